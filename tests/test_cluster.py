"""ToMATo clustering through the mesh, against the truth of synthetic clusters."""

import numpy as np
import pytest

import knnrefine

pytest.importorskip("gudhi")
from sklearn.metrics import adjusted_rand_score  # noqa: E402

from knnrefine.cluster import cluster  # noqa: E402


def blobs(seed, noise=800):
    rng = np.random.default_rng(seed)
    centres = np.array([[0.2, 0.2], [0.8, 0.3], [0.5, 0.8], [0.2, 0.75]])
    widths = [0.04, 0.05, 0.03, 0.06]
    pts = np.concatenate(
        [rng.normal(c, s, (2000, 2)) for c, s in zip(centres, widths, strict=True)]
        + [rng.random((noise, 2))]
    )
    truth = np.concatenate([np.full(2000, i) for i in range(4)] + [np.full(noise, -1)])
    return pts, truth


@pytest.mark.parametrize("k", [20, 100])
def test_finds_the_clusters_through_noise(k):
    pts, truth = blobs(0)
    cl = cluster(knnrefine.refine(pts, k), pts)
    assert cl.n_clusters == 4
    core = truth >= 0
    assert adjusted_rand_score(truth[core], cl.labels[core]) > 0.98
    assert cl.labels.shape == (len(pts),) and set(np.unique(cl.labels)) == {0, 1, 2, 3}
    # the prominences: four peaks standing far above the noise's
    assert np.isinf(cl.prominence[0]) and cl.prominence[3] > 5 * cl.prominence[4]


def test_a_cluster_across_the_periodic_seam_is_one_cluster():
    rng = np.random.default_rng(1)
    across = rng.normal([0.0, 0.5], 0.05, (2000, 2)) % 1.0  # half on each side of x = 0
    other = rng.normal([0.5, 0.5], 0.05, (2000, 2))
    pts = np.concatenate([across, other, rng.random((400, 2))])
    mesh = knnrefine.refine(pts, 40, periodic=True, box=(0, 0, 1, 1))
    cl = cluster(mesh, pts)
    assert cl.n_clusters == 2
    left = cl.labels[:2000][across[:, 0] < 0.5]
    right = cl.labels[:2000][across[:, 0] >= 0.5]
    assert np.bincount(left).argmax() == np.bincount(right).argmax()
    assert adjusted_rand_score(np.repeat([0, 1], 2000), cl.labels[:4000]) > 0.98


def test_requested_number_of_clusters():
    pts, truth = blobs(2)
    mesh = knnrefine.refine(pts, 50)
    assert cluster(mesh, pts, n_clusters=2).n_clusters == 2
    assert cluster(mesh, pts, n_clusters=4).n_clusters == 4
    with pytest.raises(knnrefine.InputError):
        cluster(mesh, pts, n_clusters=0)


# -- the number of clusters: a significance threshold, not the largest gap (issue 9, item 1) --


@pytest.mark.parametrize("k", [20, 50, 100, 200])
def test_one_gaussian_blob_is_one_cluster(k):
    """One blob of 20,000 points gave 2, 4, 3 and 6 clusters at k = 20, 50, 100, 200: the
    largest-gap rule can never answer 1."""
    pts = np.random.default_rng(0).normal(0, 1, (20_000, 2))
    cl = cluster(knnrefine.refine(pts, k), pts)
    assert cl.n_clusters == 1
    assert cl.prominence[1] < cl.threshold  # the runner-up is noise by the rule


def test_uniform_noise_is_one_cluster():
    """20,000 uniform points gave 2."""
    pts = np.random.default_rng(1).random((20_000, 2))
    assert cluster(knnrefine.refine(pts, 50), pts).n_clusters == 1


def test_blobs_of_unequal_widths_are_all_found():
    """Three blobs of widths 1.0, 2.5 and 0.5 (1,500 points) gave 2."""
    rng = np.random.default_rng(1)
    centres, widths = [[0, 0], [8, 0], [3, 6]], [1.0, 2.5, 0.5]
    pts = np.concatenate([rng.normal(c, w, (500, 2)) for c, w in zip(centres, widths, strict=True)])
    cl = cluster(knnrefine.refine(pts, 20), pts)
    assert cl.n_clusters == 3
    assert adjusted_rand_score(np.repeat([0, 1, 2], 500), cl.labels) > 0.9


def test_two_moons_are_two_clusters():
    from sklearn.datasets import make_moons

    pts, truth = make_moons(2000, noise=0.06, random_state=0)
    k = knnrefine.density.default_k(len(pts))
    cl = cluster(knnrefine.refine(pts, k), pts)
    assert cl.n_clusters == 2
    assert adjusted_rand_score(truth, cl.labels) > 0.95


def test_noise_label_marks_the_background_between_clusters():
    """With noise=True the uniform background between four blobs is mostly noise, the blobs
    keep their points, the clusters are the same ones; one blob or uniform data has none."""
    pts, truth = blobs(3, noise=2000)
    mesh = knnrefine.refine(pts, 50)
    merged, noisy = cluster(mesh, pts), cluster(mesh, pts, noise=True)
    assert merged.n_clusters == noisy.n_clusters == 4 and merged.noise == 0
    core = truth >= 0
    assert np.mean(noisy.labels[core] >= 0) > 0.95
    assert np.mean(noisy.labels[~core] < 0) > 0.6
    kept = noisy.labels >= 0
    assert np.all(noisy.labels[kept] == merged.labels[kept])
    for lone in (
        np.random.default_rng(4).random((5000, 2)),
        np.random.default_rng(4).normal(size=(5000, 2)),
    ):
        assert cluster(knnrefine.refine(lone, 50), lone, noise=True).noise == 0


@pytest.mark.parametrize("name, expected", [("franti_s1.csv", 15), ("franti_birch1.csv", 100)])
def test_benchmark_sets_have_their_number_of_clusters(name, expected):
    from conftest import load_shared

    pts = load_shared(name)
    k = knnrefine.density.default_k(len(pts))
    assert cluster(knnrefine.refine(pts, k), pts).n_clusters == expected
