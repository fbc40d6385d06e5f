"""KnnDensityEstimator: the kNN density as a scikit-learn estimator, checked against brute
force (exact k-th distances from scipy, integrals on fine grids), binomial counts of its
samples, and scikit-learn's own model-selection tools."""

import numpy as np
import pytest
from conftest import load_shared
from scipy.spatial import cKDTree

import knnrefine
from knnrefine import InputError, KnnDensityEstimator
from knnrefine.density import default_k, default_pilot_k

sklearn = pytest.importorskip("sklearn")


def mixture(n, seed=0, dim=2):
    """A wide Gaussian and a narrow one of a quarter of the points."""
    rng = np.random.default_rng(seed)
    m = n // 4
    return np.concatenate(
        [rng.normal([0.35, 0.4, 0.5][:dim], 0.1, (n - m, dim)),
         rng.normal([0.75, 0.7, 0.6][:dim], 0.02, (m, dim))]
    )  # fmt: skip


@pytest.fixture(scope="module")
def fitted():
    X = mixture(4000)
    return X, KnnDensityEstimator(k=30, method="knn").fit(X)


def grid_mean(f, lo, hi, n=400):
    """Mean of f over a fine midpoint grid of the rectangle [lo, hi]."""
    xs = lo[0] + (np.arange(n) + 0.5) * (hi[0] - lo[0]) / n
    ys = lo[1] + (np.arange(n) + 0.5) * (hi[1] - lo[1]) / n
    gx, gy = np.meshgrid(xs, ys)
    return float(np.mean(f(np.stack([gx, gy], axis=-1))))


def test_density_matches_brute_force(fitted):
    """Against k / (n pi d_k^2), d_k exact (cKDTree), normalised on a fine grid. At the mesh's
    nodes the estimate evaluates d_k exactly: there it is that function times one constant,
    the normaliser, within 2% of the brute-force one. Between nodes d_k is interpolated
    linearly (KnnDistance.error: median 1%, worst about 20% on d): the density is off by
    about 3% in the median, 25% at the 99th percentile."""
    X, est = fitted
    lo, hi = np.array(est.box_[:2]), np.array(est.box_[2:])
    tree = cKDTree(X)

    def brute(x):
        d = tree.query(x.reshape(-1, 2), k=[est.k_])[0][:, 0].reshape(x.shape[:-1])
        return est.k_ / (len(X) * np.pi * d**2)

    brute_mass = grid_mean(brute, lo, hi) * float(np.prod(hi - lo))
    nodes = est.density_.distance.nodes
    nodes = nodes[np.all((nodes >= lo) & (nodes <= hi), axis=1)]
    scale = est.density_(nodes) / brute(nodes)  # the estimate in the box (no tail_)
    np.testing.assert_allclose(scale, scale[0], rtol=1e-9)
    assert scale[0] * brute_mass == pytest.approx(1.0, abs=0.02)
    rng = np.random.default_rng(1)
    probes = np.concatenate([lo + rng.random((3000, 2)) * (hi - lo), X[:3000]])
    ratio = np.exp(est.score_samples(probes)) / (brute(probes) / brute_mass)
    assert np.median(np.abs(ratio - 1)) < 0.04
    assert np.percentile(np.abs(ratio - 1), 99) < 0.25
    assert np.abs(ratio - 1).max() < 0.7


def test_it_integrates_to_one_over_the_box(fitted):
    _, est = fitted
    lo, hi = np.array(est.box_[:2]), np.array(est.box_[2:])
    mass = grid_mean(lambda x: np.exp(est.score_samples(x)), lo, hi, n=600) * np.prod(hi - lo)
    assert mass == pytest.approx(1.0, abs=0.01)


def test_outside_the_box_and_shapes(fitted):
    X, est = fitted
    lo, hi = np.array(est.box_[:2]), np.array(est.box_[2:])
    out = est.score_samples(np.array([[hi[0] + 1e-9, 0.5], [lo[0], lo[1]], [0.5, 0.5]]))
    assert np.isfinite(out).all() and out[0] < out[2]  # no box given: tails everywhere
    cube = X[:24].reshape(2, 3, 4, 2)
    np.testing.assert_array_equal(
        est.score_samples(cube), est.score_samples(X[:24]).reshape(2, 3, 4)
    )
    assert est.score(X[:50]) == pytest.approx(est.score_samples(X[:50]).sum())
    with pytest.raises(InputError, match="x.T"):
        est.score_samples(X[:50].T)
    with pytest.raises(InputError, match="NaN"):
        est.score_samples(np.array([[np.nan, 0.5]]))


def test_periodic_estimate_wraps():
    rng = np.random.default_rng(2)
    X = np.concatenate([rng.normal(0.02, 0.05, (1500, 2)) % 1, rng.random((500, 2))])
    est = KnnDensityEstimator(k=20, method="knn", periodic=True, box=(0, 0, 1, 1)).fit(X)
    x = rng.random((200, 2))
    np.testing.assert_allclose(est.score_samples(x + [1.0, -3.0]), est.score_samples(x))
    mass = grid_mean(lambda q: np.exp(est.score_samples(q)), (0, 0), (1, 1), n=500)
    assert mass == pytest.approx(1.0, abs=0.01)
    s = est.sample(20000, random_state=0)
    assert ((s >= 0) & (s <= 1)).all()
    # the mode sits across both seams: the corner squares hold its mass
    region = (-0.1, -0.1, 0.1, 0.1)
    inside = np.all((s < 0.1) | (s > 0.9), axis=1).mean()
    p = est.density_.mass(region)
    assert abs(inside - p) < 4 * np.sqrt(p * (1 - p) / len(s))


@pytest.mark.parametrize(
    "rect", [(0.2, 0.2, 0.5, 0.6), (0.7, 0.65, 0.8, 0.75), (0.0, 0.0, 0.3, 1.0)]
)
def test_samples_follow_the_estimate(fitted, rect):
    """Counts of samples in rectangles are binomial with the estimate's exact mass there."""
    _, est = fitted
    s = est.sample(40000, random_state=3)
    x0, y0, x1, y1 = rect
    hit = np.mean((s[:, 0] >= x0) & (s[:, 0] <= x1) & (s[:, 1] >= y0) & (s[:, 1] <= y1))
    p = est.density_.mass(rect)
    assert abs(hit - p) < 4.5 * np.sqrt(p * (1 - p) / len(s))


def test_sampling_is_reproducible_and_in_the_box(fitted):
    _, est = fitted
    a = est.sample(500, random_state=7)
    np.testing.assert_array_equal(a, est.sample(500, random_state=7))
    np.testing.assert_array_equal(a, est.sample(500, random_state=np.random.default_rng(7)))
    assert est.sample(5, random_state=np.random.RandomState(1)).shape == (5, 2)
    assert not np.array_equal(a, est.sample(500, random_state=8))
    lo, hi = np.array(est.box_[:2]), np.array(est.box_[2:])
    assert ((a >= lo) & (a <= hi)).all()
    assert est.sample(0).shape == (0, 2)
    with pytest.raises(InputError, match="n_samples"):
        est.sample(-1)
    with pytest.raises(InputError, match="random_state"):
        est.sample(3, random_state="seed")


def test_sample_weights_are_relative(dim):
    """Issue 30: sample_weight is relative, as scikit-learn's and gaussian_kde's: weights
    times any factor (normalised to sum 1, times 1000) fit the same estimate at the same k,
    and the sample counts as its effective size (sum w)^2 / sum w^2, from which the default
    k comes. Equal weights are no weights. Weights of 2 against copies: the engine counts
    the weights scaled to n_eff, so k effective neighbours with weights w are k W / n_eff
    copies' worth."""
    X = mixture(800, seed=4, dim=dim)
    w = np.random.default_rng(5).integers(0, 4, len(X)).astype(float)
    n_eff = w.sum() ** 2 / (w * w).sum()
    a = KnnDensityEstimator(k=15, method="knn").fit(X, sample_weight=w)
    probes = mixture(300, seed=6, dim=dim)
    for factor in (1 / w.sum(), 1000.0):
        b = KnnDensityEstimator(k=15, method="knn").fit(X, sample_weight=w * factor)
        np.testing.assert_allclose(b.score_samples(probes), a.score_samples(probes), rtol=1e-10)
        assert b.n_samples_ == pytest.approx(n_eff)
    # no k given: the default from n_eff, whatever the weights' scale (it raised at sum 1)
    for method in ("knn", None if dim == 2 else "knn"):
        c = KnnDensityEstimator(method=method).fit(X, sample_weight=w / w.sum())
        d = KnnDensityEstimator(method=method).fit(X, sample_weight=w * 1000)
        assert c.k_ == d.k_ == (default_k if method == "knn" else default_pilot_k)(n_eff)
    # equal weights are the unweighted estimate
    plain = KnnDensityEstimator(k=15, method="knn").fit(X)
    same = KnnDensityEstimator(k=15, method="knn").fit(X, sample_weight=np.full(len(X), 7.0))
    np.testing.assert_array_equal(same.score_samples(probes), plain.score_samples(probes))
    # weights 2 on a fifth of the points, 1 on the rest: W = 6 n / 5, n_eff = 9 n / 10, the
    # engine's weights 3 / 2 and 3 / 4 (exact in binary: no rounding at the count of k)
    twice = np.where(np.arange(len(X)) % 5 == 0, 2.0, 1.0)
    ratio = twice.sum() / (twice.sum() ** 2 / (twice * twice).sum())  # W / n_eff = 4 / 3
    e = KnnDensityEstimator(k=18, method="knn").fit(X, sample_weight=twice)
    copies = KnnDensityEstimator(k=24, method="knn", box=e.box_)
    copies.fit(np.repeat(X, twice.astype(int), axis=0))
    assert 18 * ratio == pytest.approx(24)
    inside = probes[np.all((probes >= e.box_[:dim]) & (probes <= e.box_[dim:]), axis=1)]
    np.testing.assert_allclose(  # the same d_Pk: the radius holding that much weight
        e.density_.distance.exact(inside), copies.density_.distance.exact(inside), rtol=1e-12
    )
    with pytest.raises(InputError, match="sum to 0"):
        KnnDensityEstimator(k=15).fit(X, sample_weight=np.zeros(len(X)))
    with pytest.raises(InputError, match="shape"):
        KnnDensityEstimator(k=15).fit(X, sample_weight=w[:-1])
    with pytest.raises(InputError, match=">= 0"):
        KnnDensityEstimator(k=15).fit(X, sample_weight=-w)


def test_bad_parameters_are_refused_before_work():
    X = mixture(200)
    with pytest.raises(InputError, match="k must be"):
        KnnDensityEstimator(k=0).fit(X)
    with pytest.raises(InputError, match="k must be"):
        KnnDensityEstimator(k=201).fit(X)
    with pytest.raises(InputError, match="margin"):
        KnnDensityEstimator(margin=-1).fit(X)
    with pytest.raises(InputError, match="shape"):
        KnnDensityEstimator().fit(X[:, :1])


def test_scikit_learn_protocol(fitted):
    from sklearn.base import clone
    from sklearn.exceptions import NotFittedError

    est = KnnDensityEstimator(k=12, tau=4.0)
    assert est.get_params()["k"] == 12 and est.get_params()["tau"] == 4.0
    twin = clone(est)
    assert twin.get_params() == est.get_params() and twin is not est
    assert est.set_params(k=50) is est and est.k == 50
    with pytest.raises(ValueError, match="invalid parameter"):
        est.set_params(bandwith=1.0)
    assert repr(est) == "KnnDensityEstimator(k=50, tau=4.0)"
    with pytest.raises(NotFittedError):
        est.score_samples(np.zeros((1, 2)))
    X, fit = fitted
    assert fit.n_features_in_ == 2 and fit.k_ == 30
    assert isinstance(fit.mesh_, knnrefine.Mesh)


def test_grid_search_chooses_k_by_held_out_likelihood():
    """GridSearchCV and cross_val_score run on the estimator; the chosen k is the one with the
    best mean held-out log-likelihood, which the test recomputes by hand."""
    from sklearn.model_selection import GridSearchCV, KFold, cross_val_score

    X = mixture(3000, seed=8)
    cv = KFold(3, shuffle=True, random_state=0)
    ks = [4, 15, 40, 150]
    search = GridSearchCV(KnnDensityEstimator(method="knn"), {"k": ks}, cv=cv).fit(X)
    by_hand = [
        np.mean(
            [KnnDensityEstimator(k=k, method="knn").fit(X[a]).score(X[b]) for a, b in cv.split(X)]
        )
        for k in ks
    ]
    np.testing.assert_allclose(search.cv_results_["mean_test_score"], by_hand)
    assert search.best_params_["k"] == ks[int(np.argmax(by_hand))]
    assert ks[int(np.argmax(by_hand))] not in (ks[0], ks[-1])  # an interior optimum
    scores = cross_val_score(KnnDensityEstimator(k=15), X, cv=cv)
    assert scores.shape == (3,) and np.isfinite(scores).all()


def test_real_data_old_faithful():
    """Old Faithful (eruption length against waiting time: different units on the axes):
    fitted, scored on held-out rows, and sampled within the data's range."""
    X = load_shared("old_faithful.csv")[:, :2]
    rng = np.random.default_rng(0)
    order = rng.permutation(len(X))
    train, test = X[order[: len(X) * 3 // 4]], X[order[len(X) * 3 // 4 :]]
    est = KnnDensityEstimator(k=10).fit(train)
    assert np.isfinite(est.score_samples(test)).all()  # no box given: tails everywhere
    s = est.sample(2000, random_state=0)
    lo, hi = np.array(est.box_[:2]), np.array(est.box_[2:])
    assert np.all((s >= lo) & (s <= hi), axis=1).mean() > 0.99  # but the tail's few
    # two modes (short and long eruptions): both get samples
    assert (s[:, 0] < 3).mean() > 0.2 and (s[:, 0] > 3.5).mean() > 0.4


def test_k_by_cross_validation_is_the_best_of_its_curve():
    """k="cv": the curve is the mean held-out log-likelihood per point over the folds,
    recomputed here by hand with the same folds and box; k_ is its argmax."""
    from knnrefine.density.estimator import cv_folds

    X = mixture(2000, seed=9)
    est = KnnDensityEstimator(
        k="cv", method="knn", cv=4, k_grid=[3, 10, 30, 100], random_state=1
    ).fit(X)
    by_hand = []
    for k in est.cv_ks_:
        total = 0.0
        for test in cv_folds(len(X), 4, 1):
            train = np.setdiff1d(np.arange(len(X)), test)
            fold = KnnDensityEstimator(k=int(k), method="knn", box=est.box_).fit(X[train])
            total += fold.score(X[test])
        by_hand.append(total / len(X))
    np.testing.assert_allclose(est.cv_scores_, by_hand, rtol=1e-12)
    assert est.k_ == est.cv_ks_[int(np.argmax(by_hand))]
    assert est.k_ not in (3, 100)  # an interior optimum on this mixture
    # the default grid: geometric, from 4 up to a twentieth of a training fold
    auto = KnnDensityEstimator(k="cv", method="knn", cv=3).fit(X)
    assert auto.cv_ks_[0] == 4 and auto.cv_ks_[-1] == round(2000 * 2 / 3 / 20)
    assert len(auto.cv_ks_) == len(auto.cv_scores_) and np.isfinite(auto.cv_scores_).all()


@pytest.mark.slow
def test_cross_validation_keeps_copies_in_one_fold():
    """A weighted point is held out whole (folds split points): a held-out point never has
    a part of itself at distance 0 in its training fold, where k = 1 would win. Issue 30:
    weights are relative, so equal weights (all 3) are the unweighted sample (n_eff = n) and
    give its curve; copies made by repeating points are held out together too."""
    X = mixture(600, seed=10)
    w = np.full(len(X), 3)
    est = KnnDensityEstimator(k="cv", method="knn", k_grid=[1, 5, 20], cv=3)
    est.fit(X, sample_weight=w)
    assert est.k_ != 1 and np.isfinite(est.cv_scores_).all()
    assert est.n_samples_ == 600
    plain = KnnDensityEstimator(k="cv", method="knn", k_grid=[1, 5, 20], cv=3).fit(X)
    np.testing.assert_array_equal(est.cv_scores_, plain.cv_scores_)
    uneven = np.where(np.arange(len(X)) % 2 == 0, 3.0, 1.0)
    est.fit(X, sample_weight=uneven)
    assert est.k_ != 1 and np.isfinite(est.cv_scores_).all()


def test_cross_validation_parameters_are_checked():
    X = mixture(200)
    with pytest.raises(InputError, match="cv must be"):
        KnnDensityEstimator(k="cv", cv=1).fit(X)
    with pytest.raises(InputError, match="k_grid"):
        KnnDensityEstimator(k="cv", k_grid=[0, 5]).fit(X)
    with pytest.raises(InputError, match="smallest training fold"):
        KnnDensityEstimator(k="cv", method="knn", k_grid=[500]).fit(X)
    with pytest.raises(InputError, match='"cv"'):
        KnnDensityEstimator(k="auto").fit(X)


def test_periodic_without_a_box_is_refused():
    """regression: the default widened box must not become a torus's period."""
    with pytest.raises(InputError, match="box"):
        KnnDensityEstimator(k=10, periodic=True).fit(mixture(300))


@pytest.fixture(scope="module")
def replicates():
    """The sampling distribution by Monte Carlo: the estimate at 50 interior points from 40
    independent samples of the uniform density on the unit square (n = 3000, k = 30)."""
    q = 0.2 + 0.6 * np.random.default_rng(0).random((50, 2))
    values = [
        np.exp(
            KnnDensityEstimator(k=30, method="knn", box=(0, 0, 1, 1))
            .fit(np.random.default_rng(100 + r).random((3000, 2)))
            .score_samples(q)
        )
        for r in range(40)
    ]
    return q, np.array(values)


def test_standard_error_matches_the_sampling_distribution(replicates):
    """f / sqrt(k) against the spread of the estimate over independent samples (Monte Carlo
    gives 0.93 of it here: normalising over the box takes a little variance out)."""
    q, values = replicates
    est = KnnDensityEstimator(k=30, method="knn", box=(0, 0, 1, 1)).fit(
        np.random.default_rng(5).random((3000, 2))
    )
    se = est.standard_error(q)
    np.testing.assert_allclose(se, np.exp(est.score_samples(q)) / np.sqrt(30))
    ratio = np.mean(values.std(axis=0)) / np.mean(se)
    assert 0.75 < ratio < 1.15


@pytest.mark.slow
def test_bootstrap_bands_match_the_sampling_distribution(replicates):
    """The 90% band's half-width, read as 1.645 standard deviations, against the Monte Carlo
    spread; it covers the true density (1) at most probes; reproducible with random_state.
    Regression (issue 30): with weights made relative, a resample's counts were rescaled to
    its n_eff (about n / 2), so k counted twice the neighbours and the band was 0.62 of the
    spread; resamples count their repeats as copies."""
    q, values = replicates
    est = KnnDensityEstimator(k=30, method="knn", box=(0, 0, 1, 1)).fit(
        np.random.default_rng(5).random((3000, 2))
    )
    lo, hi = est.bootstrap(q, n_boot=60, level=0.9, random_state=0)
    implied_sd = np.mean((hi - lo) / (2 * 1.645))
    assert 0.7 < implied_sd / np.mean(values.std(axis=0)) < 1.3
    assert np.mean((lo <= 1.0) & (hi >= 1.0)) >= 0.8
    lo2, hi2 = est.bootstrap(q[:5], n_boot=60, level=0.9, random_state=0)
    np.testing.assert_array_equal(lo2, lo[:5])
    assert lo.shape == hi.shape == (50,)
    with pytest.raises(InputError, match="n_boot"):
        est.bootstrap(q, n_boot=1)
    with pytest.raises(InputError, match="level"):
        est.bootstrap(q, level=1.5)


def test_default_box_is_refines_widened_by_margin():
    X = mixture(500, seed=11)
    box = np.array(knnrefine.refine(X, 10).box)
    np.testing.assert_array_equal(KnnDensityEstimator(k=10, margin=0).fit(X).box_, box)
    wide = np.array(KnnDensityEstimator(k=10, margin=0.1).fit(X).box_)
    side = np.tile(box[2:] - box[:2], 2)
    np.testing.assert_allclose(wide, box + 0.1 * side * [-1, -1, 1, 1])
    # points on a line: refine's default box gives the flat side a width, the margin widens it
    line = np.column_stack([np.linspace(0, 1, 300), np.full(300, 0.5)])
    est = KnnDensityEstimator(k=10).fit(line)
    assert est.box_[3] - est.box_[1] > 0 and np.isfinite(est.score_samples(line)).all()


def test_refit_without_cv_drops_the_curve():
    """regression: a refit with a fixed k kept the curve of an earlier k="cv" fit."""
    X = mixture(600, seed=12)
    est = KnnDensityEstimator(k="cv", k_grid=[5, 20], cv=3).fit(X)
    assert hasattr(est, "cv_scores_")
    est.set_params(k=10).fit(X)
    assert est.k_ == 10 and not hasattr(est, "cv_scores_") and not hasattr(est, "cv_ks_")


def test_real_weights_are_counted_by_the_engine():
    """Issue 11: real-valued sample_weight (it raised InputError). Halving every weight is
    the same estimate (issue 30: weights are relative); against brute force the estimate at
    the mesh's nodes is k / (n_eff pi d^2) with d the least radius holding weight k once the
    weights are scaled to sum to n_eff = (sum w)^2 / sum w^2."""
    X = mixture(1500, seed=11)
    half = KnnDensityEstimator(k=30, method="knn").fit(X, sample_weight=np.full(len(X), 0.5))
    assert half.n_samples_ == 1500.0
    whole = KnnDensityEstimator(k=30, method="knn").fit(X)
    probes = mixture(300, seed=13)
    np.testing.assert_array_equal(half.score_samples(probes), whole.score_samples(probes))
    w = np.random.default_rng(12).gamma(2.0, 1.0, len(X))
    est = KnnDensityEstimator(k=20, method="knn").fit(X, sample_weight=w)
    n_eff = w.sum() ** 2 / (w * w).sum()
    assert est.n_samples_ == pytest.approx(n_eff)
    w = w * n_eff / w.sum()  # what the engine counts
    dist = est.density_.distance
    lo, hi = np.array(est.box_[:2]), np.array(est.box_[2:])
    nodes = dist.nodes[np.all((dist.nodes >= lo) & (dist.nodes <= hi), axis=1)][:400]
    d = np.hypot(*(nodes[:, None, :] - X[None, :, :]).transpose(2, 0, 1))
    order = np.argsort(d, axis=1)
    held = np.cumsum(w[order], axis=1)
    ref = np.take_along_axis(d, order, 1)[np.arange(len(nodes)), np.argmax(held >= 20, axis=1)]
    np.testing.assert_allclose(dist.exact(nodes), ref, rtol=1e-12)
    raw = 20 / (w.sum() * np.pi * ref**2)
    np.testing.assert_allclose(est.density_(nodes), raw / est.density_.raw_mass, rtol=1e-9)
    # the weighted estimate follows the weights: points weighted up in one half pull mass
    left = X[:, 0] < np.median(X[:, 0])
    tilted = KnnDensityEstimator(k=20, method="knn")
    tilted.fit(X, sample_weight=np.where(left, 3.0, 1.0))
    box = tilted.box_
    mid = np.median(X[:, 0])
    assert tilted.density_.mass((box[0], box[1], mid, box[3])) > 0.65


def test_the_default_k_is_at_most_n():
    """regression (issue 28): KnnDensityEstimator(method="knn") on 5 points raised 'k must
    be in [1, 5], got 10' though no k was given: the default is capped at n."""
    pts = np.random.default_rng(0).random((5, 2))
    est = KnnDensityEstimator(method="knn").fit(pts)
    assert est.k_ == 5 and np.isfinite(est.score_samples(pts)).all()
    assert KnnDensityEstimator().fit(pts).k_ == 5


def test_sample_weight_from_any_array_like():
    """regression (issue 28): sample_weight as a list or another array-like raised a
    TypeError (np.iscomplexobj on the raw object); pandas' nullable Float64 too. Lists,
    tuples, ranges, Series (nullable included) give the fit of the NumPy array."""
    import pandas as pd

    rng = np.random.default_rng(1)
    pts = rng.random((400, 2))
    w = rng.integers(1, 4, 400).astype(float)
    ref = KnnDensityEstimator(k=20, method="knn").fit(pts, sample_weight=w)
    for like in (list(w), tuple(w), [int(v) for v in w], pd.Series(w),
                 pd.Series(w, dtype="Float64"), pd.array(w, dtype="Float64")):  # fmt: skip
        est = KnnDensityEstimator(k=20, method="knn").fit(pts, sample_weight=like)
        np.testing.assert_array_equal(est.score_samples(pts[:50]), ref.score_samples(pts[:50]))
    with pytest.raises(knnrefine.InputError, match="finite"):
        KnnDensityEstimator(k=20).fit(pts, sample_weight=pd.Series([1.0] * 399 + [None],
                                                                 dtype="Float64"))  # fmt: skip


@pytest.mark.parametrize("method", [None, "knn"])
def test_grid_is_in_the_datas_units(dim, method):
    """est.grid gives the cells' centres in the data's units (inside box_) and the density
    there as score_samples does, whitened or not, in the plane and in space (issue 30)."""
    if dim == 3 and method is None:
        method = "knn"  # the default in space
    X = mixture(3000, seed=21, dim=dim) * [10.0, 0.5, 3.0][:dim] + [100.0, -2.0, 7.0][:dim]
    est = KnnDensityEstimator(k=40, method=method).fit(X)
    shape = (12, 15) if dim == 2 else (5, 6, 7)
    *axes, values = est.grid(shape)
    assert values.shape == shape and [len(a) for a in axes] == list(shape[::-1])
    lo, hi = np.array(est.box_[:dim]), np.array(est.box_[dim:])
    for a, axis in enumerate(axes):
        assert (axis > lo[a]).all() and (axis < hi[a]).all()
    mesh = np.meshgrid(*axes, indexing="xy") if dim == 2 else np.meshgrid(*axes, indexing="ij")
    centres = np.stack([m.ravel() for m in mesh], axis=1)
    want = np.exp(est.score_samples(centres))
    got = values.ravel() if dim == 2 else values.transpose(2, 1, 0).ravel()
    np.testing.assert_allclose(got, want, rtol=1e-6)
    with pytest.raises(InputError, match="shape"):
        est.grid((0, 3))


def test_feature_names_are_kept_and_checked():
    """Fitted on a DataFrame with named columns, the estimator keeps their names as
    scikit-learn does (feature_names_in_), refuses queries whose columns are named otherwise,
    and takes plain arrays; a refit on an array forgets them (issue 30)."""
    pd = pytest.importorskip("pandas")
    X = mixture(800, seed=22)
    frame = pd.DataFrame(X, columns=["lon", "lat"])
    est = KnnDensityEstimator(k=20, method="knn").fit(frame)
    assert list(est.feature_names_in_) == ["lon", "lat"]
    np.testing.assert_array_equal(est.score_samples(frame), est.score_samples(X))
    with pytest.raises(InputError, match="columns"):
        est.score_samples(frame[["lat", "lon"]])
    assert not hasattr(est.fit(X), "feature_names_in_")


def test_held_out_points_beyond_the_box_score_finitely_without_a_box(dim):
    """Issue 30: fitted without a box, the estimate has tails everywhere (a Cauchy density of
    one point's weight about the fitted box), so that held-out points beyond the data's box
    score finitely; it still integrates to 1 and samples follow it; with a box given, the
    estimate is 0 outside it as before."""
    method = None if dim == 2 else "knn"
    X = mixture(3000, seed=4, dim=dim)
    est = KnnDensityEstimator(k=40, method=method).fit(X)
    tail = est.tail_
    assert tail is not None and tail.weight == pytest.approx(1 / 3000)
    lo, hi = np.array(est.box_[:dim]), np.array(est.box_[dim:])
    far = np.array([hi + 1.0, lo - 50.0, [hi[0] + 0.01, *lo[1:] + 0.1]])
    inside = X[:200]
    got = est.score_samples(far)
    np.testing.assert_allclose(got, np.log(tail.weight * tail(far)), rtol=1e-12)
    # inside: the box estimate and the tail, mixed
    box_only = est.density_(inside)
    want = np.log((1 - tail.weight) * box_only + tail.weight * tail(inside))
    np.testing.assert_allclose(est.score_samples(inside), want, rtol=1e-12)
    # the tail's mass in the box by its own draws: box part + tail part integrate to 1
    draws = tail.sample(400000, np.random.default_rng(0))
    in_box = np.mean(np.all((draws >= lo) & (draws <= hi), axis=1))
    shape = (200, 200) if dim == 2 else (40, 40, 40)
    *axes, values = est.grid(shape)
    cell = np.prod([a[1] - a[0] for a in axes])
    assert values.sum() * cell == pytest.approx(1 - tail.weight + tail.weight * in_box, abs=2e-3)
    # the tail's density is the t density with one degree of freedom (scipy)
    from scipy.stats import multivariate_t

    ref = multivariate_t(loc=tail.centre, shape=np.diag(tail.scale**2), df=1)
    np.testing.assert_allclose(tail(far), ref.pdf(far), rtol=1e-10)
    # samples: a share of about weight * P(outside) beyond the box
    s = est.sample(60000, random_state=1)
    assert np.mean(~np.all((s >= lo) & (s <= hi), axis=1)) < 10 * tail.weight
    # with a box given: 0 outside it, as before
    boxed = KnnDensityEstimator(k=40, method=method, box=est.box_).fit(X)
    assert boxed.tail_ is None and np.isneginf(boxed.score_samples(far)).all()


def test_cross_validation_scores_are_finite_with_outliers_in_held_out_folds():
    """Issue 30 (regression): a held-out point beyond the training folds' box scored -inf,
    which made cross_val_score unusable on data with a few far points."""
    sklearn = pytest.importorskip("sklearn.model_selection")
    rng = np.random.default_rng(3)
    X = np.concatenate([mixture(2000, seed=3), rng.normal(0.5, 3.0, (6, 2))])
    rng.shuffle(X)
    scores = sklearn.cross_val_score(KnnDensityEstimator(k=30), X, cv=3)
    assert np.isfinite(scores).all()
