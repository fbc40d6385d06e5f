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
